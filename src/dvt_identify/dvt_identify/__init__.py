"""dvt_identify."""
