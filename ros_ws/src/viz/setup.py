from glob import glob

from setuptools import setup

package_name = "viz"

setup(
    name=package_name,
    version="0.1.0",
    packages=["pusher_viz"],  # the Python module: PyPI has a package called viz
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*")),
    ],
    install_requires=["setuptools"],
    extras_require={"test": ["pytest"]},  # colcon test runs test/ with pytest
    zip_safe=True,
    maintainer="pusher-rl maintainers",
    maintainer_email="maintainers@pusher-rl.invalid",
    description="The arm in RViz and Foxglove: markers of any task's arm from its joint states.",
    license="Apache-2.0",
    # Kept a literal list: ros_ws/tools/ros_install.py reads it to generate lib/viz/<exe>.
    entry_points={
        "console_scripts": [
            "markers = pusher_viz.markers:main",
            "live_view = pusher_viz.live_view:main",
        ]
    },
)
