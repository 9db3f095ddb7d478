"""The daemon's web page (drivers/web/page.py): live view, plots, health, set-up, recordings."""

from drivers.web.page import SettingsBackend, WebPage, undistorted_preview
from drivers.web.settings import WebSettings

__all__ = ["SettingsBackend", "WebPage", "WebSettings", "undistorted_preview"]
