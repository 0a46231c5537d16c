"""Per run and scene: slices dropped, full (gen-2) garbage collections and the longest, the longest delay of a slice's
release behind its scan end (the player stalled), and the process's cores (CPU seconds / wall seconds)."""
import json, glob, sys
print(__doc__.strip())
for f in sorted(glob.glob(sys.argv[1] + '/r*_*/replay.json')):
    d = json.load(open(f))
    for si, rec in enumerate(d['modes']['streaming']['recordings']):
        sl = rec['slices']
        g = (rec.get('gc_pauses') or {}).get('gen2')
        gc = 'not measured' if g is None else f"{g['collections']} (longest {g['max_ms']:.1f} ms)"
        pl = rec.get('phase_lock') or {}
        extra = f", held back {pl['yields']} times ({pl['yielded_ms']:.0f} ms)" if pl.get('yields') else ''
        print(f"{f.split('/')[-2]} scene {si}: dropped {sum(x['dropped'] for x in sl)}, gen-2 collections {gc}, "
              f"release delay max {1e3 * max(x['release_s'] - x['scan_end_s'] for x in sl):.1f} ms, "
              f"process {rec['process_cpu_s'] / rec['wall_s']:.2f} cores{extra}")
