"""The paper's figures (Alhaija et al. 2020, Tables 1 and 3), keyed by run label: printed beside
ours in reports, and named in `iae-eval seeds` where an ordering is one the paper measured."""
from __future__ import annotations

# Table 1: FID, KID x100 (256x512, 16,000 real photos)
PAPER_TABLE1 = {"CycleGAN": (103.3, 10.2), "MUNIT": (99.0, 13.5), "Ours (full)": (47.6, 4.2),
                "Ours, w/o shared discr.": (59.2, 4.8), "Ours, w/o decomp. cycle": (99.6, 11.8),
                "Ours, w/o A": (88.7, 5.4), "Ours, w/o N": (60.2, 4.9), "Ours, w/o F": (56.7, 5.9)}
# Table 3: normal mean (deg), albedo L1, reflection L1 (0-255); no rows for the input ablations
PAPER_TABLE3 = {"Ours, w/o shared discr.": (17.75, 54.00, 55.60), "Ours, w/o decomp. cycle": (18.80, 67.21, 71.00),
                "CycleGAN": (27.82, 68.18, 73.18), "MUNIT": (29.15, 81.44, 74.75), "Ours (full)": (14.73, 52.74, 51.74)}

# eval.seeds' column names -> (table, position)
_COLUMN_SOURCE = {"normals (deg)": (PAPER_TABLE3, 0), "albedo L1": (PAPER_TABLE3, 1), "reflection L1": (PAPER_TABLE3, 2),
                  "FID": (PAPER_TABLE1, 0), "KID x100": (PAPER_TABLE1, 1)}


def paper_value(label: str, column: str) -> float | None:
    """The paper's figure for a run label in one of eval.seeds' columns, None where it has none."""
    table, pos = _COLUMN_SOURCE.get(column, ({}, 0))
    row = table.get(label)
    return None if row is None else row[pos]
