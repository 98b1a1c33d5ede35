"""dvt_model."""
