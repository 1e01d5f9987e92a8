import sys

from emulators.ur.controller import main

sys.exit(main())
