"""The simulated plant: a controller + transmission that speaks the wire protocol.

* :mod:`~dvt_driver.plant.core` - the simulated controller and physics (pure, stepped);
* :mod:`~dvt_driver.plant.hidden` - the hidden effects the identifier must find (presets in
  ``config/``);
* :mod:`~dvt_driver.plant.server` - ``dvt-plant``: the core on a pseudo-terminal in real time;
* :mod:`~dvt_driver.plant.offline` - the driver's supervisor and the core without ROS or a pty.
"""
