"""seqshape.errors: the errors survive the trip from a worker process (pickling)."""

import pickle

import pytest

from seqshape._runner import WorkerPool
from seqshape.errors import ConfigError, DataError, MissingDependencyError, SeqshapeError


@pytest.mark.parametrize("line", [None, 0, 12])
def test_data_error_pickles_whole(line):
    err = DataError("logs/a b.json", "expected 17 columns, got 3", line=line)
    err.add_note("while labelling log 0003")
    back = pickle.loads(pickle.dumps(err))
    assert type(back) is DataError
    assert (back.path, back.message, back.line) == ("logs/a b.json",
                                                    "expected 17 columns, got 3", line)
    assert str(back) == str(err) == ("logs/a b.json: expected 17 columns, got 3"
                                     if line is None else
                                     f"logs/a b.json:{line}: expected 17 columns, got 3")
    assert back.__notes__ == ["while labelling log 0003"]


def test_a_data_error_subclass_pickles_as_itself():
    class ShortFile(DataError):
        pass

    globals()["ShortFile"] = ShortFile  # pickle finds classes by module and name
    ShortFile.__qualname__ = "ShortFile"
    try:
        back = pickle.loads(pickle.dumps(ShortFile("x.bin", "cut short", 4)))
        assert type(back) is ShortFile and str(back) == "x.bin:4: cut short"
    finally:
        del globals()["ShortFile"]


@pytest.mark.parametrize("err", [ConfigError("--workers must be >= 1, got 0"),
                                 MissingDependencyError("needs pyarrow"),
                                 SeqshapeError("offline replay: unknown track 'a'")])
def test_the_other_errors_pickle(err):
    back = pickle.loads(pickle.dumps(err))
    assert type(back) is type(err) and str(back) == str(err)


def _fail(path: str):
    raise DataError(path, "bad header", line=2)


def test_a_data_error_raised_in_a_worker_reaches_the_parent():
    """A spawned worker's DataError is re-raised here, whole (one that does not unpickle
    kills the pool's result thread: the wait would never end, hence the timeout)."""
    with WorkerPool(1) as pool:
        task = pool.submit(_fail, "a.txt")
        with pytest.raises(DataError) as info:
            task.get(timeout=60)
    assert (info.value.path, info.value.message, info.value.line) == ("a.txt", "bad header", 2)
    assert str(info.value) == "a.txt:2: bad header"
