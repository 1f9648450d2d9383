"""The ``lrms`` command line (see :mod:`service.cli.main`)."""
