"""streamdet.export"""
