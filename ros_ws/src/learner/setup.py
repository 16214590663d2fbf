from glob import glob

from setuptools import setup

package_name = "learner"

setup(
    name=package_name,
    version="0.1.0",
    packages=["pusher_learner"],  # the Python module: named so it cannot clash with a PyPI package
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
    description="The online HIL-SERL learner: fine-tunes the prior from live transitions and publishes weights.",
    license="Apache-2.0",
    # Kept a literal list: ros_ws/tools/ros_install.py reads it to generate lib/learner/<exe>.
    entry_points={"console_scripts": ["node = pusher_learner.node:main"]},
)
