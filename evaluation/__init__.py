"""streamdet.evaluation"""
