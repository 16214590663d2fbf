from glob import glob

from setuptools import setup

package_name = "policy"

setup(
    name=package_name,
    version="0.1.0",
    packages=["pusher_policy"],  # the Python module: PyPI has a package called policy
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
        "Serves a trained checkpoint: answers every /pusher/state with /policy/action; hot-reloads"
        " the checkpoint file."
    ),
    license="Apache-2.0",
    # Kept a literal list: ros_ws/tools/ros_install.py reads it to generate lib/policy/<exe>.
    entry_points={"console_scripts": ["node = pusher_policy.node:main"]},
)
