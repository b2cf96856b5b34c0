"""Skip markers for tests that need an optional extra. Checked with ``find_spec``: collecting a module then
does not import the extra on every xdist worker, as ``importorskip`` at module level would."""

from __future__ import annotations

import importlib.util

import pytest

needs_openai = pytest.mark.skipif(
    importlib.util.find_spec("openai") is None,
    reason="the openai backend needs the openai SDK (pip install 'vlmproprio[openai]')",
)
