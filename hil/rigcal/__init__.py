"""Rig calibration (issue 18): hand-eye from many robot poses (camera -> robot and TCP -> flange
markers, solved jointly), device time offsets, the rig calibration file, and the adapters that
apply the offsets. Knows no concrete driver: the procedure goes through the driver interfaces.
"""
