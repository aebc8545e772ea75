"""The sharded Arrow cache, one module per role.

- :mod:`~phigenesis.data.cache.files`: the layout's names, atomic writes, scene ids as file names;
- :mod:`~phigenesis.data.cache.checksums`: the shards' CRCs, :class:`ShardInfo`, column byte ranges;
- :mod:`~phigenesis.data.cache.sink`: the byte sink under a shard's IPC writer;
- :mod:`~phigenesis.data.cache.writer`: :class:`ShardWriter`;
- :mod:`~phigenesis.data.cache.manifest`: :class:`Manifest`, its checks and shard paths;
- :mod:`~phigenesis.data.cache.reader`: :class:`ShardReader`, :class:`CacheReader`;
- :mod:`~phigenesis.data.cache.verify`: :func:`verify_cache`.

:mod:`phigenesis.data.shards` re-exports the public names of all of them (the cache's one import
path for the rest of the toolkit).
"""
