"""`python -m drgan.pipeline ...`: drgan.pipeline.runner.main."""

import sys

from drgan.pipeline.runner import main

sys.exit(main())
