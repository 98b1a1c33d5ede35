"""Running things: experiments, child processes, discovery, Foxglove and the link benchmark
(the launcher is in the integration layer, :mod:`dvt_driver.system`).

* :mod:`~dvt_driver.run.schedule` - experiment schedules as data: commands, limits, signals (pure);
* :mod:`~dvt_driver.run.experiment_core` - the named experiments (pure);
* :mod:`~dvt_driver.run.experiment` - ``dvt-experiment``: sends a schedule to the driver;
* :mod:`~dvt_driver.run.processes` - child processes of the launcher and the benchmarks;
* :mod:`~dvt_driver.run.bench` - ``dvt-bench link``: throughput and CPU of the chain.
"""
