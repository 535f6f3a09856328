"""The seed's rectification experiments (seed 000 Tables 3, 4-5 and 6, blunders), printed beside the seed.

Run:  python benchmarks/bench_adjust.py
"""

from __future__ import annotations

import time

import numpy as np

from geocoder.adjust.experiments import block_table, blunder_case, edge_table, single_frame_table

SEED_T3 = {10: (11.8, 102.5), 15: (0.6, 13.2), 25: (0.5, 10.8), 40: (0.5, 10.4), 81: (0.5, 9.9)}
SEED_T5 = [(90.8, None), (79.9, None), (66.2, 75.8), (69.8, 72.2), (67.9, 67.9)]


def main() -> None:
    t0 = time.perf_counter()
    print("Table 3: check RMS (m), single MSS-like frame, perfect data (seed: Kansas frame)")
    print("| control (seed) | control (ours) | collinearity seed | collinearity ours | polynomial seed | polynomial ours |")
    print("|---:|---:|---:|---:|---:|---:|")
    for n, r in zip(SEED_T3, single_frame_table(perfect=True)):
        print(f"| {n} | {r['control']} | {SEED_T3[n][0]} | {r['collinearity']:.2f} | {SEED_T3[n][1]} | {r['polynomial']:.2f} |")
    print("\nTables 4-5: 3 x 3 block, check RMS (m), block adjustment / single frames (mean over frames)")
    print("| case | control | ties | seed BA/SF | ours BA | ours SF | sigma0 |")
    print("|---:|---:|---:|---|---:|---:|---:|")
    for k, r in enumerate(block_table()):
        ba, sf = SEED_T5[k]
        print(f"| {k + 1} | {r['control']} | {r['ties']} | {ba}/{sf if sf else '-'} | {r['block_total']:.1f} | "
              f"{np.nanmean(r['single_rms']):.1f} ({np.isnan(r['single_rms']).sum()} failed) | {r['sigma0']:.2f} |")
    r = blunder_case()
    print("\nBlunders: 5 % of tie observations displaced by 5-50 px (case 1 control)")
    print("| blunders | found | false alarms | check RMS clean | contaminated | robust + snooping |")
    print("|---:|---:|---:|---:|---:|---:|")
    print(f"| {r['blunders']} | {r['found']} | {r['false_alarms']} | {r['clean_rms']:.1f} | {r['contaminated_rms']:.1f} | {r['robust_rms']:.1f} |")
    print("\nTable 6: check RMS (m), single frame, edge pairs as control (mean +- std over replicates);")
    print("configuration 0 = the same number of conventional control points")
    rows = edge_table(counts=(25, 41, 81, 145), configurations=tuple(range(1, 11)), replicates=5)
    print("| configuration | " + " | ".join(f"{n} pairs" for n in (25, 41, 81, 145)) + " |")
    print("|---:|" + "---:|" * 4)
    for cfg in range(0, 11):
        cells = [f"{r['mean']:.1f} +- {r['std']:.1f}" for r in rows if r["configuration"] == cfg]
        print(f"| {cfg} | " + " | ".join(cells) + " |")
    print(f"\n{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
