"""streamdet.calibration"""
