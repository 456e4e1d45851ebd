"""Test-wide settings.

Under CI (the environment variable CI is set, as `.ci/run` runs) hypothesis draws the same
examples every run, so a submission's result does not depend on the draw; a developer's runs
keep exploring new examples and its database replays any failure found.
"""

import os

from hypothesis import settings

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")
