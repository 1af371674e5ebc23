"""pyserial URL handlers of lfrig's own, found the way pyserial finds ``loop://`` in
``serial.urlhandler``: ``serial.protocol_handler_packages`` lists this package (``rig.grbl.open_port``
adds it), and ``serial.serial_for_url("SCHEME://...")`` imports ``rig.urlhandler.protocol_SCHEME``.

- ``fakegrbl://``: the simulated GRBL controller (:mod:`rig.urlhandler.protocol_fakegrbl`).
"""
