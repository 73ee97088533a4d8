"""A missing prerequisite skips a test where it may be missing and fails it on CI, which installs every one."""
import pytest

from prerequisites import missing


def test_a_missing_prerequisite_skips_with_what_to_install(monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    with pytest.raises(pytest.skip.Exception, match="apt-get install chromium"):
        missing("headless Chromium is missing: apt-get install chromium chromium-driver")


def test_on_ci_a_missing_prerequisite_fails(monkeypatch):
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="LPIPS weights .* install step is broken"):
        missing("LPIPS weights not installed: run `make install`")
