#!/usr/bin/env python3
"""How far sampled vehicles stray from the paths their recordings take.

Usage: path_distance.py LOG_DIR ROLLOUT_DIR [--list]

LOG_DIR holds the recorded trajectories as rollout JSON (`drivescript convert SCENE -o
LOG_DIR/ID.json`), ROLLOUT_DIR a run's samples (ID_0.json). For each vehicle that moves at
least 5 m in its recorded future (20 or more observed steps), it takes the largest distance,
over the sample's future steps, from the recorded future's path (the polyline of its
positions), and prints the median, 75th and 90th percentiles and the shares above 0.5, 1 and
2 m; with --list, the ten largest. Where a sample goes on after its recording stops
(unconditional runs) the distance also counts that part, so compare conditional runs.

Only the Python standard library.
"""
import json, math, sys, glob, os
def seg_dist(p, a, b):
    ax, ay = a; bx, by = b; px, py = p
    dx, dy = bx-ax, by-ay; L = dx*dx+dy*dy
    t = 0 if L == 0 else max(0, min(1, ((px-ax)*dx+(py-ay)*dy)/L))
    return math.hypot(px-ax-t*dx, py-ay-t*dy)
out = []
for lf in sorted(glob.glob(sys.argv[1]+'/*.json')):
    sid = os.path.basename(lf)[:-5]
    rf = os.path.join(sys.argv[2], sid+'_0.json')
    if not os.path.exists(rf): continue
    L = json.load(open(lf)); R = json.load(open(rf)); c = L['current_step']
    la = {a['id']: a for a in L['agents']}
    for a in R['agents']:
        if a['type'] != 'vehicle' or a['id'] not in la: continue
        ls = [s for s in la[a['id']]['states'][c:] if s[3]]
        if len(ls) < 20: continue
        path = [(s[0], s[1]) for s in ls]
        if math.hypot(path[-1][0]-path[0][0], path[-1][1]-path[0][1]) < 5: continue  # movers only
        m = 0
        for s in a['states'][c+1:]:
            if not s[3]: continue
            d = min(seg_dist((s[0], s[1]), path[i], path[i+1]) for i in range(len(path)-1))
            m = max(m, d)
        out.append((m, sid, a['id']))
out.sort()
n = len(out)
print(n, 'movers; max distance from the recorded path: median %.2f, p75 %.2f, p90 %.2f; >0.5 m %.3f, >1 m %.3f, >2 m %.3f' % (
    out[n//2][0], out[3*n//4][0], out[9*n//10][0], sum(o[0]>0.5 for o in out)/n, sum(o[0]>1 for o in out)/n, sum(o[0]>2 for o in out)/n))
if '--list' in sys.argv[3:]:
    for o in out[-10:]: print('%.2f %s %s' % o)
