import sys

from online_id.cli import main

sys.exit(main())
