import sys

from uhrnet.cli import main

sys.exit(main())
