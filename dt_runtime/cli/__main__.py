"""`python -m dt_runtime.cli ...` is `dt ...`."""
import sys

from dt_runtime.cli.main import main

sys.exit(main())
