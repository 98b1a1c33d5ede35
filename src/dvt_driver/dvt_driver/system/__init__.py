"""The integration layer: the one place where the driver and the identifier meet.

Everything else in :mod:`dvt_driver` runs without :mod:`dvt_identify`, and :mod:`dvt_identify`
never imports :mod:`dvt_driver` (both depend on :mod:`dvt_model` only; the import contracts in
``pyproject.toml`` make the CI fail otherwise). What composes the packages into a running
system lives here and depends on both (``package.xml``: ``dvt_identify``):

* :mod:`~dvt_driver.system.launch` - ``dvt-launch``: plant, driver, model node, recorders,
  experiment, the identifier's supervisor (``--supervise``: its episode records arrive on the
  contract's topic) and the Foxglove bridge as processes; its options
  (:mod:`~dvt_driver.system.launch_args`), its rclpy monitor (:mod:`~dvt_driver.system.monitor`)
  and the recording's check (:mod:`~dvt_driver.system.bagcheck`);
* :mod:`~dvt_driver.system.bench_detect` - ``dvt-bench loop``: change detection on the live
  chain (plant, driver, model node);
* :mod:`~dvt_driver.system.bench_loop` - ``dvt-bench loop --with-identifier``: live episodes of
  the self-closing loop and their figures;
* :mod:`~dvt_driver.system.bench` - the ``dvt-bench`` dispatch over the three packages'
  benchmarks;
* :mod:`~dvt_driver.system.demo` - the README's demo (``scripts/demo.sh``).
"""
