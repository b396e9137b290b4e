"""`python -m drgan STAGE [KEY=VALUE ...]`: the `drgan` console command (drgan.cli) where its script is not on the
PATH."""

import sys

from drgan.cli import main

sys.exit(main())
