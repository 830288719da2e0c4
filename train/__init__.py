"""Entry points: `python -m train --help`."""
