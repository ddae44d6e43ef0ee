r"""Continues saved live sessions in a new process (for
test_session.py): for every tracker name given, loads FOLDER/<name>.pt,
streams the rest of the test realization and saves the outputs to
FOLDER/<name>.out.pt."""
import sys

import torch

from helpers import gen, live_trackers, stream_realization, tiny_scenario
from tg_nebp.filters import TrackingSession


def main(folder, start, *names):
    data = tiny_scenario(6).generate(gen(3))
    for name in names:
        session = TrackingSession.load(f'{folder}/{name}.pt',
                                       live_trackers()[name]())
        with torch.no_grad():
            outputs = stream_realization(session, data, start=int(start))
        torch.save([(o.mean, o.cov) for o in outputs],
                   f'{folder}/{name}.out.pt')


if __name__ == '__main__':
    main(*sys.argv[1:])
