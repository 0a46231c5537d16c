"""streamdet.runtime_ort"""
