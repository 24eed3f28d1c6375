import sys

from fppsim.cli import main

sys.exit(main())
