import sys

from train.cli import interruptible_main

sys.exit(interruptible_main("python -m train"))
