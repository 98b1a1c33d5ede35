"""dvt_driver."""
