"""The daemon's web page (drivers/web/page.py): live view, plots, health, set-up, recordings.

Only the settings are exported here: the page itself (`drivers.web.page`) pulls in aiohttp,
~20 MB of a Pi's memory that a daemon with the page off should not carry, so the wiring
imports it only when the page is on.
"""

from drivers.web.settings import WebSettings

__all__ = ["WebSettings"]
