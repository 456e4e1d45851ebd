"""What the smoother's Bayes tree holds, read from GTSAM's own drawing of it (shared by the
smoother's tests)."""

import re

from autonomy.vins.fixed_lag import FixedLagSmoother


def root_frontals(smoother: FixedLagSmoother) -> list[str]:
    """The variables of the Bayes tree's root clique, as GTSAM names them ("x29"). GTSAM's
    ``dot`` writes each clique before its children, so the first label is a root's; a root has
    no separator (the part after " : ")."""
    label = re.search(r'label="([^"]*)"', smoother._isam.dot()).group(1)
    return [name.strip() for name in label.split(":")[0].split(",")]
