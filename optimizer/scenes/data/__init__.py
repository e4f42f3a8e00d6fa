"""External assets: manifests (``data_manifests/*.toml``), a resumable verified fetcher, scene packs.

``camo data list | fetch | verify | pack`` (:mod:`optimizer.scenes.data.cli`). The manifest format is described in
:mod:`optimizer.scenes.data.manifest` and ``data_manifests/README.md``; downloading, checksum verification and safe
unpacking in :mod:`optimizer.scenes.data.fetch`. Only the standard library touches the network.
"""

from optimizer.scenes.data.cli import register

__all__ = ["register"]
