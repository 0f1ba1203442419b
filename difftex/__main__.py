import sys

from difftex.cli import main

sys.exit(main())
