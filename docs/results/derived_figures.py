"""Print the figures of docs/results/README.md that are read from JSON or computed, not copied from a `.md`.

Run from the repository root: `python3 docs/results/derived_figures.py`. Standard library only; it reads
the benchmark folders next to it and the paper's Table 1 and Flickering-Atari figures typed in below.
"""

import json
from pathlib import Path

HERE = Path(__file__).resolve().parent
DOMAINS = ("lightdark10d", "kidnapped20d", "mtt20d")

# Table 1 of the paper (average position error: mean, s.e.), typed from its LaTeX source.
PAPER_TABLE1 = {
    "escort": ((0.347, 0.03), (9.063, 0.51), (3.665, 0.31)),
    "escort_nocorr": ((0.381, 0.07), (10.246, 0.35), (4.213, 0.59)),
    "escort_notemp": ((0.321, 0.03), (10.859, 0.51), (3.874, 0.43)),
    "escort_noproj": ((0.359, 0.09), (9.654, 0.32), (3.90, 0.42)),
    "svgd": ((0.379, 0.03), (10.906, 0.49), (4.295, 0.22)),
    "dvrl": ((1.557, 0.10), (14.309, 0.60), (4.33, 0.09)),
    "pomcpow": ((2.12, 0.24), (12.023, 0.55), (4.611, 0.09)),
}
# The paper's Flickering-Atari table, Pong (50M frames).
PAPER_PONG = {"escort_latent": 17.97, "dvrl": 18.17}

# (row label, folder, method, paper row): the folder each Table 1 row of the results page is read from.
TABLE1_ROWS = (
    ("ESCORT", "fidelity/domains_lambda0.1", "escort", "escort"),
    ("ESCORT-NoCorr", "fidelity/domains_lambda0.1", "escort_nocorr", "escort_nocorr"),
    ("ESCORT-NoTemp", "domains_compiled", "escort_notemp", "escort_notemp"),
    ("ESCORT-NoProj", "fidelity/domains_lambda0.1", "escort_noproj", "escort_noproj"),
    ("SVGD", "domains_compiled", "svgd", "svgd"),
    ("SIR", "domains_compiled", "sir", None),
    ("DVRL", "dvrl", "dvrl", "dvrl"),
)
POMCPOW_ROWS = (
    ("POMCPOW (SIR belief)", "closed_loop_pomcpow", "pomcpow_sir", "pomcpow"),
    ("POMCPOW (ESCORT belief)", "closed_loop_pomcpow", "pomcpow_escort", "pomcpow"),
)


def load(path):
    return json.loads((HERE / path).read_text())


def protocol_a(folder, method):
    data = load(f"{folder}/domains.json")
    cells = {}
    for row in data["rows"]:
        if row["method"] == method and row["particles"] == data["particles"]:
            mean, se = row["summary"]["final_error"]
            cells[row["domain"]] = (mean, se, len(row["seeds"]), data["domain_info"][row["domain"]]["steps"])
    return cells


def protocol_b(folder, method):
    data = load(f"{folder}/closed_loop.json")
    cells = {}
    for row in data["rows"]:
        if row["method"] == method:
            s = row["summary"]
            error = (s["final_position_error"], s["final_position_error_se"])
            cells[row["domain"]] = (*error, s["episodes"], row["steps"])
    return cells


def table1():
    print("Table 1: final position error, ours (mean ± s.e., seeds or episodes, steps) / paper,")
    print("  ours/paper, z = (ours − paper) / sqrt(s.e.² + paper s.e.²)")
    rows = [(label, folder, protocol_a(folder, method), paper) for label, folder, method, paper in TABLE1_ROWS]
    rows += [(label, folder, protocol_b(folder, method), paper) for label, folder, method, paper in POMCPOW_ROWS]
    for label, folder, cells, paper in rows:
        parts = []
        for i, domain in enumerate(DOMAINS):
            mean, se, n, steps = cells[domain]
            if paper:
                p_mean, p_se = PAPER_TABLE1[paper][i]
                z = (mean - p_mean) / (se**2 + p_se**2) ** 0.5
                ref = f"{p_mean} ± {p_se}, ours/paper {mean / p_mean:.2f}, z {z:+.1f}"
            else:
                ref = "-"
            parts.append(f"{mean:.3f} ± {se:.3f} (n={n}, T={steps}) / {ref}")
        print(f"  {label:24s} [{folder}] " + " | ".join(parts))


def atari():
    print("Flickering Pong: ours (last 100 games) / paper, difference")
    for row in load("atari_pong/atari.json")["rows"]:
        mean, se = row["return"]
        paper = PAPER_PONG.get(row["agent"])
        diff = f", paper − ours {paper - mean:.2f}" if paper is not None else ""
        print(f"  {row['agent']:14s} {mean:.2f} ± {se:.2f} ({row['games']} games, {row['seeds']} seed){diff}")


if __name__ == "__main__":
    table1()
    atari()
