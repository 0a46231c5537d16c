"""streamdet.benchmarks"""
