import sys

from awaremw.cli import main

sys.exit(main())
