"""``lungdeform view``: bad input exits 2 with one line on stderr."""

import socket

from lungdeform.cli.main import main
from lungdeform.playback.export import glb_bytes
from tests.browser.support import two_lungs


def test_view_port_in_use_exits_2_naming_the_address(tmp_path, capsys):
    # another program listens on the port: one line naming host:port and the option to change,
    # before anything is served (the server is never started)
    model = tmp_path / "m.glb"
    model.write_bytes(glb_bytes(two_lungs(2)))
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        assert main(["view", str(model), "--port", str(port)]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and f"127.0.0.1:{port}" in err[0] and "--port" in err[0]
    assert "viewer for" not in captured.out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.glb"]  # nothing written
