"""hil_sim."""
