"""dvt_driver: see the package README section in the repository README."""

# BLAS held to one thread in this process: dvt_model.one_blas_thread, one place for the three
# packages (importing dvt_model runs it)
import dvt_model as _dvt_model  # noqa: F401
