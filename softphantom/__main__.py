import sys

from softphantom.cli import main

sys.exit(main())
