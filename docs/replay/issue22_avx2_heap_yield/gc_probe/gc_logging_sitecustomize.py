import gc, time, sys, atexit
_t = {}
_log = []
def _cb(phase, info):
    if phase == "start":
        _t[0] = time.perf_counter()
    else:
        d = time.perf_counter() - _t.get(0, time.perf_counter())
        if info["generation"] == 2 or d > 0.005:
            _log.append((time.monotonic(), info["generation"], d * 1e3, info.get("collected")))
gc.callbacks.append(_cb)
def _dump():
    with open("/tmp/s18/gclog/gc.txt", "w") as f:
        for r in _log: f.write("%.3f gen%d %.1f ms collected %s\n" % r)
atexit.register(_dump)
