"""Visualisation of a running RRA system (Rerun). Importing this package never imports rerun."""
