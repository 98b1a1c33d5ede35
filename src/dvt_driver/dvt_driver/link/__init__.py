"""The link to the controller: wire codec, serial port, session, clock, safety, driver node.

* :mod:`~dvt_driver.link.protocol` - the wire protocol (frames, messages; pure codec);
* :mod:`~dvt_driver.link.serial_link` - a pyserial port speaking it (reconnectable, counted);
* :mod:`~dvt_driver.link.session` - the controller session as a pure state machine (HELLO,
  CONFIG, answers, stream timeout, keep-alive, reconnect);
* :mod:`~dvt_driver.link.clock` - controller clock -> ROS time (pure);
* :mod:`~dvt_driver.link.safety` - limits, refusals, watchdog, trips, gear shifts (pure);
* :mod:`~dvt_driver.link.settings` - the driver's validated settings (pure);
* :mod:`~dvt_driver.link.node` - ``dvt_driver_node``, the thin rclpy layer over the above.
"""
