"""Ground mapping: calibration, inverse perspective mapping, occupancy grid, frontiers.

Pure functions on numpy arrays (no I/O except the calibration file helpers, no asyncio).
Frame conventions are in `app.mapping.frames`.
"""
