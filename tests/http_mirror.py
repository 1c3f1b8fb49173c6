"""A folder served over HTTP from a thread, as a dataset mirror (`URL/<dataset>/<path>`), for the
fetch tests (`tests/test_data_fetch.py`) and `benchmarks/bench_fetch.py`: no network needed."""
from __future__ import annotations

import http.server
import socket
import threading
import time
from pathlib import Path


class Mirror:
    """A folder served over HTTP in a thread; `requests` counts the GETs, `cut` names files whose
    first response breaks off after half their bytes, `slow` adds a delay per 64 kB."""

    def __init__(self, root: Path):
        self.root, self.requests, self.cut, self.slow = root, [], set(), 0.0
        mirror = self

        class Handler(http.server.SimpleHTTPRequestHandler):
            def __init__(self, *args, **kwargs):
                super().__init__(*args, directory=str(root), **kwargs)

            def log_message(self, *args):
                pass

            def do_GET(self):
                mirror.requests.append(self.path)
                path = root / self.path.lstrip("/")
                if not path.is_file():
                    return self.send_error(404)
                data = path.read_bytes()
                self.send_response(200)
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                if self.path in mirror.cut:
                    mirror.cut.discard(self.path)
                    self.wfile.write(data[: len(data) // 2])
                    self.wfile.flush()
                    self.connection.shutdown(socket.SHUT_RDWR)
                    return
                for start in range(0, len(data), 1 << 16):
                    self.wfile.write(data[start:start + (1 << 16)])
                    if mirror.slow:
                        time.sleep(mirror.slow)

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        self.thread = threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True)
        self.thread.start()

    def put(self, path: str, data: bytes) -> None:
        target = self.root / "broad" / path
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)

    def close(self):
        self.server.shutdown()
        self.server.server_close()
