"""The new muscles against Damas 2016 and Seynnes 2007: per-group mwf growth (results/cohort-new), the VL CSA course
under data/damas.toml (results/cohort-damas) and the quadriceps (RF+VL+VM+VI, CSA summed over each subject-side)
under data/seynnes.toml (results/cohort-seynnes); writes docs/new-muscles.png.  python jobs/new_muscles.py"""

import glob
from collections import defaultdict

import h5py
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from hyper.runs import measured


def series(path):
    with h5py.File(path) as f:
        return f["t"][()], f["csa_ratio"][()], f["volume_ratio"][()], float(f.attrs["csa0_m2"])


# per muscle group and protocol: the final CSA and volume increase, mean (min, max) over subjects and sides
PROTOCOLS = ("mwf", "every3days", "weekly")
g = defaultdict(lambda: ([], []))
for protocol in PROTOCOLS:
    for p in sorted(glob.glob(f"results/cohort-new/runs/*_{protocol}.h5")):
        name = p.split("/")[-1][: -len(f"_{protocol}.h5")]
        t, c, v, _ = series(p)
        g[name.split("_")[0], protocol][0].append(100 * (c[-1] - 1))
        g[name.split("_")[0], protocol][1].append(100 * (v[-1] - 1))
heads = [f"{what} {p}" for what in ("CSA", "volume") for p in PROTOCOLS]
print("| muscle | n | " + " | ".join(heads) + " |")
for m in ("RF", "VL", "VM", "VI", "GM"):
    cells = []
    for which in (0, 1):
        for protocol in PROTOCOLS:
            x = np.array(g[m, protocol][which])
            cells.append(f"+{x.mean():.2f} % (+{x.min():.2f}, +{x.max():.2f})" if len(x) else "–")
    print(f"| {m} | {len(g[m, 'mwf'][0])} | " + " | ".join(cells) + " |")
fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4), layout="constrained")


def at(t, c, week):
    return np.interp(168 * week, t, c)


print("damas VL: week 3, 10")
for p in sorted(glob.glob("results/cohort-damas/runs/*_damas.h5")):
    t, c, v, _ = series(p)
    n = p.split("/")[-1][:-9]
    a.plot(t / 168, c, label=n)
    print(n, round(at(t, c, 3), 4), round(at(t, c, 10), 4))
d = measured.read("data/damas.csv")  # its CSA / CSA0 after time 0
a.plot(d.t / 168, d.csa_ratio, "ko", label="Damas 2016 (VL)")
a.set(xlabel="week", ylabel="CSA / CSA0", title="vastus lateralis, damas.toml (2/week, 10 weeks)")
a.legend(fontsize=8)
quad = defaultdict(dict)
for p in sorted(glob.glob("results/cohort-seynnes/runs/*_seynnes.h5")):
    n = p.split("/")[-1][:-11]
    m, s, side = n.split("_")
    quad[f"{s}_{side}"][m] = series(p)
print("seynnes quadriceps: week 3, 5")
for k, ms in sorted(quad.items()):
    if len(ms) < 4:
        print(k, "incomplete", sorted(ms))
        continue
    t = ms["VL"][0]
    tot0 = sum(s[3] for s in ms.values())
    q = sum(s[1] * s[3] for s in ms.values()) / tot0
    b.plot(t / 168, q, label=f"quadriceps {k} ({tot0 * 1e4:.0f} cm²)")
    print(k, round(at(t, q, 3), 4), round(at(t, q, 5), 4), "CSA0 sum", round(tot0 * 1e4, 1))
s = measured.read("data/seynnes.csv")
b.plot(s.t / 168, s.csa_ratio, "ko", label="Seynnes 2007 (quadriceps)")
b.set(xlabel="week", ylabel="CSA / CSA0", title="RF+VL+VM+VI, seynnes.toml (3/week, 5 weeks)")
b.legend(fontsize=8)
fig.savefig("docs/new-muscles.png", dpi=100)
print("data damas", d.csa_ratio, "seynnes", s.csa_ratio)
