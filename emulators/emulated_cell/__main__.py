import sys

from emulators.emulated_cell.cell import main

sys.exit(main())
