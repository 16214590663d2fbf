from glob import glob

from setuptools import setup

package_name = "corrections"

setup(
    name=package_name,
    version="0.1.0",
    packages=["pusher_corrections"],  # the Python module: PyPI has a package called corrections
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
    description="HIL-SERL corrections: the policy/human command mux and the (scripted or keyboard) corrector.",
    license="Apache-2.0",
    # Kept a literal list: ros_ws/tools/ros_install.py reads it to generate lib/corrections/<exe>.
    entry_points={
        "console_scripts": [
            "mux = pusher_corrections.mux:main",
            "corrector = pusher_corrections.corrector:main",
        ]
    },
)
