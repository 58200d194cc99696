import sys

from cifemu.cli import main

sys.exit(main())
