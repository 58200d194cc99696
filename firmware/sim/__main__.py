import sys

from firmware.sim.cli import main

sys.exit(main())
