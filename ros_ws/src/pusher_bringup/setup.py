from glob import glob

from setuptools import setup

package_name = "pusher_bringup"

setup(
    name=package_name,
    version="0.1.0",
    packages=[],  # launch files only
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/launch", glob("launch/*.launch.yaml")),
        ("share/" + package_name + "/config", glob("config/*.xml")),
    ],
    install_requires=["setuptools"],
    extras_require={"test": ["pytest"]},  # colcon test runs test/ with pytest
    zip_safe=True,
    maintainer="pusher-rl maintainers",
    maintainer_email="maintainers@pusher-rl.invalid",
    description="Launch files of the pusher-rl pipelines.",
    license="Apache-2.0",
    entry_points={"console_scripts": []},
)
