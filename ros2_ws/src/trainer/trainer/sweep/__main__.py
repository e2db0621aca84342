import sys

from trainer.sweep.cli import main

sys.exit(main())
