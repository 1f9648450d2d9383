"""Servo motion drivers: one :class:`~drivers.servo.interface.Motor` interface, CiA 402 semantics.

* :mod:`drivers.servo.interface` - the Motor interface, :class:`DriveConfig`, samples, errors
* :mod:`drivers.servo.cia402` - pure CiA 402 / CiA 301 definitions and decoders
* :mod:`drivers.servo.cia402_can` - CANopen backend on python-can (``canopen+<interface>://``)
"""
