"""python -m benchmarks run NAME | render"""

import sys

from . import main

sys.exit(main(sys.argv[1:]))
