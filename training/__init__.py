"""streamdet.training"""
