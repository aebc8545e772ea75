"""PhiGenesis: 4D driving-scene caches and lightweight 4D Gaussian models.

Data: :mod:`phigenesis.prep` builds, verifies and previews caches (the functions behind
``phigenesis-prep``); :mod:`phigenesis.data.loader` reads them into torch.
"""

__version__ = "0.1.0"
