# (thirty-fifth session) run from the repository root as: .venv/bin/python docs/replay/issue22_line_dropout/stalls/watch.py STREAMDET-REPLAY-OPTIONS...
"""Run streamdet-replay with a watchdog thread: it sleeps 1 ms in a loop and, whenever it wakes more than 12 ms
late, records the other threads' current stacks (the thread that held the GIL has just released it)."""
import json
import sys
import threading
import time
import traceback
events = []
def watchdog():
    me = threading.get_ident()
    last = time.perf_counter()
    while True:
        time.sleep(0.001)
        now = time.perf_counter()
        late = (now - last - 0.001) * 1e3
        if late > 12:
            frames = sys._current_frames()
            names = {t.ident: t.name for t in threading.enumerate()}
            stacks = {names.get(i, str(i)): [f"{fs.filename.split('streamdet')[-1]}:{fs.lineno} {fs.name}" for fs in traceback.extract_stack(f)[-6:]]
                      for i, f in frames.items() if i != me}
            events.append({"t": now, "late_ms": late, "stacks": stacks})
        last = now
threading.Thread(target=watchdog, daemon=True, name="watchdog").start()
from streamdet.cli_utils import replay_main
try:
    replay_main()
except SystemExit:
    pass
json.dump(events, open("watchdog_events.json", "w"), indent=1)
print("watchdog events:", len(events), "late ms:", sorted(round(e["late_ms"]) for e in events))
