import sys

from brainmech.main import main

sys.exit(main())
