"""The depth projection's parts by role; the stage is :mod:`phigenesis.data.stages.project`."""
