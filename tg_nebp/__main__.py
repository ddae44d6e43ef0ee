import sys

from tg_nebp.cli import main

sys.exit(main())
