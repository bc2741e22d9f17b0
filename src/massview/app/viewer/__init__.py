"""The web viewer: an HTTP/WebSocket server on the destination rank and its page."""

from .server import ViewerServer
from .state import ViewerState

__all__ = ["ViewerServer", "ViewerState"]
