from glob import glob

from setuptools import setup

package_name = "sim"

setup(
    name=package_name,
    version="0.1.0",
    packages=["pusher_sim"],  # the Python module: PyPI has a package called sim
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    extras_require={"test": ["pytest"]},  # colcon test runs test/ with pytest
    zip_safe=True,
    maintainer="pusher-rl maintainers",
    maintainer_email="maintainers@pusher-rl.invalid",
    description=(
        "The pusher-reach MuJoCo arm as a ROS 2 node: publishes state, target and transitions,"
        " obeys commands (realtime or lockstep)."
    ),
    license="Apache-2.0",
    # Kept a literal list: ros_ws/tools/ros_install.py reads it to generate lib/sim/<exe>.
    entry_points={"console_scripts": ["node = pusher_sim.node:main"]},
)
