"""The ament resource index: ``ros2_shim.ament_index``, shared with the launch reader."""

from ros2_shim.ament_index import executables, package_prefix, package_share, packages, prefixes

__all__ = ["executables", "package_prefix", "package_share", "packages", "prefixes"]
