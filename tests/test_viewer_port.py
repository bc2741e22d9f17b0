"""``massview view`` on a port something else holds: one line saying so, before any scene is
loaded or rank started (``--port 0``, which the line suggests, is tested serving in
tests/test_launcher_signals.py)."""

from __future__ import annotations

import socket

import pytest

from conftest import SMALL_SCENE, run_cli
from massview.core.errors import ConfigError


@pytest.fixture()
def held_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]


def _message(port: int) -> str:
    return f"massview: error: port {port} on 127.0.0.1 is in use; pass --port another (e.g. --port 0 picks a free one)"


@pytest.mark.parametrize("extra", [[], ["--ranks", "2"], ["--system", "reliefboards", "--ranks", "2"]],
                         ids=["1-rank", "2-ranks", "reliefboards"])
def test_a_port_in_use_is_one_line_before_anything_starts(held_port, extra):
    proc = run_cli("view", SMALL_SCENE, "--port", held_port, "--size", "320x240", *extra, check=False, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip() == _message(held_port), proc.stderr
    assert "serving" not in proc.stdout


def test_the_server_says_the_same_when_the_port_is_taken_after_the_check(held_port):
    from massview.app.viewer.server import ViewerServer, check_port

    check_port("127.0.0.1", 0)  # port 0 always binds
    with pytest.raises(ConfigError) as e:
        check_port("127.0.0.1", held_port)
    assert str(e.value) == _message(held_port)[len("massview: error: "):]
    with pytest.raises(ConfigError) as e:
        ViewerServer(None, "127.0.0.1", held_port).start()
    assert str(e.value) == _message(held_port)[len("massview: error: "):]


def test_render_only_options_given_to_view_are_named_as_ignored(held_port):
    """view accepts render's flags (one parser) but writes nothing and steers its own camera:
    --out, --frames, --path ... given to it are named, not silently dropped."""
    proc = run_cli("view", SMALL_SCENE, "--port", held_port, "--frames", 3, "-o", "xx", "--reference", check=False, timeout=120)
    assert "massview: note: view ignores -o, --frames, --reference" in proc.stderr, proc.stderr
    quiet = run_cli("view", SMALL_SCENE, "--port", held_port, "--size", "320x240", check=False, timeout=120)
    assert "note" not in quiet.stderr
