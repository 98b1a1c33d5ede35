"""The simulated plant: a controller + transmission that speaks the wire protocol.

* :mod:`~dvt_driver.plant.core` - the simulated controller's firmware, :class:`PlantSim` (pure,
  stepped), with its settings in :mod:`~dvt_driver.plant.settings`;
* :mod:`~dvt_driver.plant.physics` - the transmission it drives: the physics and the hidden
  effects' forces (pure);
* :mod:`~dvt_driver.plant.hidden` - the hidden effects the identifier must find (presets in
  ``config/``);
* :mod:`~dvt_driver.plant.server` - ``dvt-plant``: the core on a pseudo-terminal in real time;
* :mod:`~dvt_driver.plant.offline` - the driver's supervisor and the core without ROS or a pty.
"""
