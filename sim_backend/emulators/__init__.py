"""Protocol-level device emulators used by the test-suite (loopback-only network traffic)."""
