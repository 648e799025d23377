"""The curves of curves.json (relMSE against seconds, prepass included; `bench` points at
doubling spp), rex at session 29's budget ("before", commit 7d554bd) and this session's
("after"), beside path, one panel per scene:

    .venv/bin/python docs/results/shape-order-sharp-light-2026-11-29/figure.py
"""
import json
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
curves = json.load(open(os.path.join(HERE, "curves.json")))
fig, axes = plt.subplots(1, len(curves), figsize=(4 * len(curves), 3.6))
style = {"path": ("k", "-"), "rex before": ("tab:blue", "--"), "rex after": ("tab:red", "-")}
for ax, (scene, rows) in zip(axes, curves.items()):
    for name, pts in rows.items():
        colour, line = style[name]
        ax.loglog([p[1] for p in pts], [p[2] for p in pts], line, color=colour, marker="o",
                  ms=3, label=name)
    ax.axhline(0.01, color="grey", lw=0.8, ls=":")
    ax.set_title(scene)
    ax.set_xlabel("seconds (prepass included)")
axes[0].set_ylabel("relMSE")
axes[0].legend()
fig.tight_layout()
fig.savefig(os.path.join(HERE, "rex-curves.png"), dpi=90)
