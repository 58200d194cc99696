import sys

from dbm_tools.cli import main

sys.exit(main())
