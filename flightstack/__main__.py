# PYTHON_ARGCOMPLETE_OK
"""`python -m flightstack ...` runs the operator CLI."""

from flightstack.cli.app import main

raise SystemExit(main())
