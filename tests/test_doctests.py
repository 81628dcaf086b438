"""Run the docstring examples of the modules that carry them."""

import doctest
import importlib

import pytest

MODULES = ["seqshape.geometry", "seqshape.errors", "seqshape.camera", "seqshape.data.av2", "seqshape.data.nuscenes",
           "seqshape.scripts.tracks"]


@pytest.mark.parametrize("name", MODULES)
def test_doctests(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0 and result.failed == 0
