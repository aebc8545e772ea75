"""The unified semantic taxonomy now lives in :mod:`phigenesis.taxonomy` (core: the models use it
too); this name stays for code written against the old path. Import from there."""

from phigenesis.taxonomy import *  # noqa: F403
