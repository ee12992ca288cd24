"""``surftrack recover``: an MCAP file cut off at any point (SIGKILL, a crash, a full disk) is rewritten into
a finished file holding exactly the messages that were readable, in order."""

from __future__ import annotations

import numpy as np
import pytest
from mcap.reader import make_reader

from surftrack.cli import main
from surftrack.io.mcap_writer import TrackWriter


def _messages(path) -> list[tuple[str, int, bytes]]:
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None  # a finished file: summary and footer
        return [(c.topic, m.log_time, m.data) for _, c, m in reader.iter_messages(log_time_order=False)]


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    path = tmp_path_factory.mktemp("log") / "run.mcap"
    with TrackWriter(path, {"video": "v.mp4"}, chunk_size=4096) as w:  # small chunks: many cut points
        for i in range(300):
            w.poses(i / 10, {"lnd.0.shaft": (np.eye(3), np.array([1.0, 2.0, 100.0 + i]))})
            w.status(i / 10, "lnd.0.shaft", "tracking", 0.5, {})
    return path


@pytest.mark.parametrize("keep", [0.05, 0.3, 0.5, 0.8, 0.999, 1.0])
def test_recover_keeps_every_readable_message(log, tmp_path, capsys, keep):
    data = log.read_bytes()
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(data[:int(len(data) * keep)])
    fixed = tmp_path / "fixed.mcap"
    assert main(["recover", str(broken), "-o", str(fixed)]) == 0
    out = capsys.readouterr().out
    got, original = _messages(fixed), _messages(log)
    assert got == original[:len(got)]  # a prefix, unchanged
    assert f"surftrack recover: {len(got)} messages" in out
    if keep == 1.0:
        assert len(got) == len(original) and "(the whole file)" in out
    else:
        assert "(the file ends inside a record)" in out
    if keep >= 0.3:
        assert len(got) >= keep * len(original) - 150  # at most a chunk or so is lost
    with open(fixed, "rb") as f:
        assert next(make_reader(f).iter_metadata()).metadata == {"video": "v.mp4"}
    if keep == 1.0:  # the summary's copies of schemas and channels are not registered a second time
        with open(fixed, "rb") as f, open(log, "rb") as g:
            s, t = make_reader(f).get_summary(), make_reader(g).get_summary()
        assert sorted(c.topic for c in s.channels.values()) == sorted(c.topic for c in t.channels.values())
        assert len(s.schemas) == len(t.schemas)


def test_recover_refuses_what_it_cannot_do(log, tmp_path, capsys):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file")
    assert main(["recover", str(junk), "-o", str(tmp_path / "x.mcap")]) == 2
    assert "junk.mcap: not an MCAP file" in capsys.readouterr().err
    assert main(["recover", str(log), "-o", str(log)]) == 2
    assert "must not overwrite the file it is recovered from" in capsys.readouterr().err
    assert main(["recover", str(tmp_path / "missing.mcap"), "-o", str(tmp_path / "y.mcap")]) == 2
    assert "missing.mcap" in capsys.readouterr().err
