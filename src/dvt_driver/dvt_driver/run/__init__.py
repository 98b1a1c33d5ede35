"""Running things: experiments, the launcher and the link benchmark.

* :mod:`~dvt_driver.run.experiment_core` - experiment schedules (pure);
* :mod:`~dvt_driver.run.experiment` - ``dvt-experiment``: sends a schedule to the driver;
* :mod:`~dvt_driver.run.launch` - ``dvt-launch``: plant/driver/model/recorder/experiment chain;
* :mod:`~dvt_driver.run.bench` - ``dvt-bench link``: throughput and CPU of the chain.
"""
