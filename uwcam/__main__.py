import sys

from uwcam.cli import main

sys.exit(main())
