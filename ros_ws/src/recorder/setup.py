from glob import glob

from setuptools import setup

package_name = "recorder"

setup(
    name=package_name,
    version="0.1.0",
    packages=["pusher_recorder"],  # the Python module: PyPI has a package called recorder
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="pusher-rl maintainers",
    maintainer_email="maintainers@pusher-rl.invalid",
    description="Drives the sim with the scripted expert / random actions (or listens passively) "
                "and records a rosbag2 dataset.",
    license="Apache-2.0",
    # Kept a literal list: ros_ws/tools/ros_install.py reads it to generate lib/recorder/<exe>.
    entry_points={"console_scripts": ["node = pusher_recorder.node:main"]},
)
