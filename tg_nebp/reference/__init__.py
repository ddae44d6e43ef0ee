r"""The paper's published results: the two curves of its Fig. 2 (outage
probability versus error threshold, and P(accept H0) of the two-sided
chi-square NEES test versus confidence level, BP and NEBP), digitized from
the paper's plot files."""
import csv
from importlib import resources
from typing import Dict, Tuple

__all__ = ['paper_curves', 'PAPER_TABLE']

#: The outage probabilities and P(accept H0) of BP and NEBP, read off
#: Fig. 2 (test network, 400 realizations).
PAPER_TABLE = {
    'bp': {'outage': {'0.5': 0.571, '1.0': 0.161, '2.0': 0.020},
           'accept': {'0.50': 0.232, '0.95': 0.590, '0.99': 0.708}},
    'nebp': {'outage': {'0.5': 0.377, '1.0': 0.054, '2.0': 0.007},
             'accept': {'0.50': 0.505, '0.95': 0.946, '0.99': 0.985}},
}


def paper_curves() -> Dict[Tuple[str, str], Tuple[list, list]]:
    r"""Returns :obj:`{(figure, series): (x, y)}` with :obj:`figure` in
    :obj:`"outage"`, :obj:`"consistency"` and :obj:`series` in :obj:`"BP"`,
    :obj:`"NEBP"`."""
    curves = {}
    path = resources.files('tg_nebp.reference') / 'figure2_digitized.csv'
    with path.open() as f:
        for row in csv.DictReader(f):
            x, y = curves.setdefault((row['figure'], row['series']), ([], []))
            x.append(float(row['x']))
            y.append(float(row['y']))
    return curves
