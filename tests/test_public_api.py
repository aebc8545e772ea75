"""The public API: ``phigenesis.<name>`` for what the README shows, loaded on first use."""

from __future__ import annotations

import subprocess
import sys

import pytest

import phigenesis


def test_import_phigenesis_is_light():
    code = "import sys, phigenesis; print(sorted(m for m in ('torch', 'cv2', 'pyarrow') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("name", [n for n in phigenesis.__all__ if n != "__version__"])
def test_every_public_name_is_the_object_its_module_defines(name: str):
    import importlib

    module = importlib.import_module(phigenesis._API[name])
    expected = module if name == "prep" else getattr(module, name)
    assert getattr(phigenesis, name) is expected
    assert name in dir(phigenesis)


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'train_stage3'"):
        phigenesis.train_stage3  # noqa: B018
    assert phigenesis.__version__ == phigenesis.version.__version__
