"""Device drivers for the LRMS rig.

One folder per device. Each wire codec is sans-I/O (bytes in, typed telegrams out, and back);
transports (TCP, python-can, pyserial) are thin layers around it. Devices are opened by URL
through :mod:`drivers.url`.
"""
