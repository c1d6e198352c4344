"""One-off (session 12): the root lag's ratio prior widened from (1e-3, 3) to (1e-3, 30), on the
two tests whose root stayed below 90% (results.md, results.json here):

    nice python experiments/results/mangrove/wide_lag_prior/run_wide_lag.py --models lag+creep+ar1 \
        --tests halloran_10,gladstone_21 --warmup 150 --samples 200 --out /tmp/mg_wide
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[4]))
import treeinfer.inference.pulltest.posterior as P  # noqa: E402

P.LAG_RATIO_PRIOR = (1e-3, 30.0)
from experiments import mangrove  # noqa: E402

sys.exit(mangrove.main(sys.argv[1:]))
