"""A live camera stream without a camera: an HTTP MJPEG stream of given JPEG parts, served on 127.0.0.1.

``localize ROUTE.tlm http://127.0.0.1:PORT/stream.mjpg`` reads it as it reads a
network camera (:mod:`topoloc.datasets.sources.live`); the tests of live sources
and ``benchmarks/bench_reliability.py`` serve their frames (and bad parts) so.
"""

from __future__ import annotations

import http.server
import socketserver
import threading
import time


class MjpegServer:
    """An HTTP MJPEG stream (``multipart/x-mixed-replace``) of ``parts`` at ``fps``, looped ``loops`` times.

    Each client that connects gets the stream from its first part; :meth:`close`
    ends every stream and the server.  ``url`` is where it is served.
    """

    def __init__(self, parts: list[bytes], *, fps: float = 20.0, loops: int = 1) -> None:
        served = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                try:
                    for _ in range(served.loops):
                        for data in parts:
                            if served.closed.is_set():
                                return
                            self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n"
                                             % len(data) + data + b"\r\n")
                            time.sleep(1.0 / served.fps)
                except (BrokenPipeError, ConnectionResetError):  # the client stopped reading
                    return

            def log_message(self, *args: object) -> None:
                pass

        self.fps, self.loops = fps, loops
        self.closed = threading.Event()
        self.server = socketserver.ThreadingTCPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/stream.mjpg"

    def close(self) -> None:
        self.closed.set()
        self.server.shutdown()
        self.server.server_close()


__all__ = ["MjpegServer"]
