"""Recordings: the only code that writes, reads, pairs, recovers and summarises them (pure)."""
