"""The client never resends a request that creates something once the connection broke after it was sent.

Independent truth: what a server saw. The stand-in below is a raw TCP server that reads each request in full
(headers and body), counts it, and closes the connection without answering: the request reached the server,
the answer never came (httpx.RemoteProtocolError, a dropped connection). A POST that creates a batch or a path
must then raise ConnectionFailed with the server having seen exactly one request (a resend could create the
batch twice); a GET on the same server is resent (1 + retries requests), which shows that the drop is the kind
the client does retry when that is safe."""
from __future__ import annotations

import asyncio
import socket
import threading

import pytest

from shadowopt.api.client import AsyncClient, Client, ConnectionFailed

RETRIES = 3


class DropAfterRequest:
    """Reads whole HTTP/1.1 requests, records (method, path, body) and closes without a response."""

    def __init__(self):
        self.seen: list[tuple[str, str, bytes]] = []
        self.sock = socket.socket()
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(16)
        self.sock.settimeout(0.05)  # accept() wakes up to see close()
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}"
        self._stop = False
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self):
        while not self._stop:
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with conn:
                conn.settimeout(5)
                data = b""
                try:
                    while b"\r\n\r\n" not in data:
                        chunk = conn.recv(65536)
                        if not chunk:
                            break
                        data += chunk
                    if b"\r\n\r\n" not in data:
                        continue
                    head, body = data.split(b"\r\n\r\n", 1)
                    lines = head.decode("latin-1").split("\r\n")
                    length = 0
                    for line in lines[1:]:
                        k, _, v = line.partition(":")
                        if k.strip().lower() == "content-length":
                            length = int(v.strip())
                    while len(body) < length:
                        chunk = conn.recv(65536)
                        if not chunk:
                            break
                        body += chunk
                    method, path, _ = lines[0].split(" ", 2)
                    self.seen.append((method, path, body))
                except OSError:
                    pass
            # closing without a byte of response: the client sees the connection drop

    def close(self):
        self._stop = True
        self._thread.join(timeout=5)
        self.sock.close()


@pytest.fixture
def dropping():
    srv = DropAfterRequest()
    yield srv
    srv.close()


RIG = {"camera": {"usd_path": "/World/Camera"}, "lights": [{"type": "directional", "direction": [0, -1, 0]}]}


def test_a_batch_or_path_submission_whose_connection_drops_raises_and_is_sent_once(dropping):
    with Client(dropping.url, token="t", retries=RETRIES, backoff_s=0.01) as c:
        with pytest.raises(ConnectionFailed):
            c.submit_batch("s1", [RIG])
        assert [(m, p) for m, p, _ in dropping.seen] == [("POST", "/v1/batches")]
        assert b'"scene_id":"s1"' in dropping.seen[0][2].replace(b" ", b"")  # the whole body reached the server
        with pytest.raises(ConnectionFailed):
            c.submit_path("s1", RIG, usd_camera="/World/Camera", time=(0, 2, 1))
        assert [(m, p) for m, p, _ in dropping.seen] == [("POST", "/v1/batches"), ("POST", "/v1/paths")]
        # the same drop on a GET (idempotent) is resent: 1 + RETRIES requests
        with pytest.raises(ConnectionFailed):
            c.batch("b1")
    assert [p for _, p, _ in dropping.seen[2:]] == ["/v1/batches/b1"] * (1 + RETRIES)


def test_the_async_client_does_not_resend_a_batch_submission_either(dropping):
    async def go():
        async with AsyncClient(dropping.url, token="t", retries=RETRIES, backoff_s=0.01) as c:
            with pytest.raises(ConnectionFailed):
                await c.submit_batch("s1", [RIG])
            with pytest.raises(ConnectionFailed):
                await c.batch("b1")

    asyncio.run(go())
    assert [(m, p) for m, p, _ in dropping.seen] == [("POST", "/v1/batches")] + [("GET", "/v1/batches/b1")] * (1 + RETRIES)
