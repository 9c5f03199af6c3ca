import sys

from sitl_bridge.cli import main

sys.exit(main())
