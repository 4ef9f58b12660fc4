"""The DJI/Ryze Tello: driver (`driver.TelloDriver`), its configuration and errors (`config`), its parts
(command link, state stream, phase tracker, takeoff and land, sticks, watchdog, rejoin, video), its SDK
3.0 video commands (`sdk_video`), its preflight and its velocity-step identification. docs/drivers.md,
"Tello driver", says how they fit."""
