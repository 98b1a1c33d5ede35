"""Recording on the ROS side: the ``dvt-recorder`` node and the ``dvt-bag`` tool.

* :mod:`~dvt_driver.recording.policy` - which topics to record and with which QoS (pure);
* :mod:`~dvt_driver.recording.node` - node ``dvt_recorder`` (``dvt-recorder``), a thin wrapper
  around :class:`dvt_model.recording.BagRecorder`;
* :mod:`~dvt_driver.recording.bagtool` - ``dvt-bag info|recover``.

Writing, reading, recovering and summarising bags is :mod:`dvt_model.recording`'s job alone.
"""
