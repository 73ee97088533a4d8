"""What a test does when something outside the project that it needs is missing."""
import os
from typing import NoReturn

import pytest


def missing(what: str) -> NoReturn:
    """Skips the test, the message saying what is missing and how to get it; on CI (CI=true), whose .ci/run installs
    every such prerequisite, fails instead, so a broken install step cannot pass as a skip."""
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(f"{what} (CI installs it, so its install step is broken)")
    pytest.skip(what)
