"""``python -m visnerf``: the command line (``visnerf.cli``); ``torchrun -m visnerf train ...`` starts it
on several processes."""

import sys

from visnerf.cli import main

sys.exit(main())
