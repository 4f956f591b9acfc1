import sys

from sdh2svc.cli import main

sys.exit(main())
