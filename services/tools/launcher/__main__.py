import sys

from services.tools.launcher.cli import main

sys.exit(main())
