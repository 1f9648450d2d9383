"""The rig coordinator, REST service, scheduler, result store and the ``lrms`` command line."""
