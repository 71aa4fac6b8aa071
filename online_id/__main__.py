import sys

from online_id.cli import main

if __name__ == "__main__":  # not when multiprocessing's spawn imports this module in a worker process
    sys.exit(main())
