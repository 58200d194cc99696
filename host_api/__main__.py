import sys

from host_api.status import main

sys.exit(main())
