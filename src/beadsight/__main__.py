import sys

from beadsight.cli import main

sys.exit(main())
