"""Offline tools around the core: replay statistics, drawing, calibration, the monitor's view."""
