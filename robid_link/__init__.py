"""robid_link: automatic dynamic-model identification of industrial robots.

The worker lives in :mod:`robid_link.ident`; the daemon in :mod:`robid_link.link`.
"""

__version__ = "0.1.0"
__all__ = ["__version__"]
