# PYTHON_ARGCOMPLETE_OK
"""`python -m flightstack ...` runs the operator CLI."""

from flightstack.cli import main

raise SystemExit(main())
