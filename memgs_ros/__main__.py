import sys

from memgs_ros.cli import main

sys.exit(main())
