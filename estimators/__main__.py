import sys

from .cli import main

if __name__ == "__main__":  # not when a child process re-imports the main module (multiprocessing)
    sys.exit(main())
