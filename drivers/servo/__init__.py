"""Servo motion drivers: one :class:`~drivers.servo.interface.Motor` interface, CiA 402 semantics.

* :mod:`drivers.servo.interface` - the Motor interface, :class:`DriveConfig`, samples, errors,
  and :class:`Cia402Motor`, the CiA 402 behaviour every backend shares
* :mod:`drivers.servo.cia402` - pure CiA 402 / CiA 301 definitions and decoders
* :mod:`drivers.servo.cia402_can` - CANopen backend on python-can (``canopen+<interface>://``)
* :mod:`drivers.servo.modbus_backend` - Modbus RTU backend on pyserial (``modbus-rtu://``)

Open a motor by URL: ``drivers.url.open_device("motor", url, config=DriveConfig(...))``.
See docs/servo.md and docs/modbus.md.
"""
