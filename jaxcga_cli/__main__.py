"""Runs the ``jaxcga`` command: ``python -m jaxcga_cli ...``."""

import sys

from jaxcga_cli.main import main

sys.exit(main())
