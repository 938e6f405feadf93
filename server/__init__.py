"""crowdslam server: the only package with I/O (HTTP, WebSocket, SQL, MCAP, files, CLI)."""

from importlib.metadata import version

__version__ = version("crowdslam")
"""The installed package's version (``pyproject.toml``): the API's OpenAPI version and ``--version``."""
