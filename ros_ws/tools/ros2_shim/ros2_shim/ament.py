"""The ament resource index: ``offline_rl_core.ament_index``, shared with the launch reader."""

from offline_rl_core.ament_index import executables, package_prefix, package_share, packages, prefixes

__all__ = ["executables", "package_prefix", "package_share", "packages", "prefixes"]
