import sys

from drivers.emulated_cell.cell import main

sys.exit(main())
