"""streamdet.models"""
