"""``python -m dbm_tools``: ``cifemu dbm``, file and card commands.

The card commands are host_api's (``host_api.dbm_commands``); only this entry point
reaches across, the package's modules never import host_api.
"""

import sys

from host_api.dbm_commands import main

sys.exit(main())
