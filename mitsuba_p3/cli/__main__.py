"""``python -m mitsuba_p3.cli``: the command line."""
from . import main

main()
