"""streamdet.data"""
