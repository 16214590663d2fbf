from setuptools import setup

package_name = "pusher_common"

setup(
    name=package_name,
    version="0.1.0",
    packages=[package_name],
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    extras_require={"test": ["pytest"]},  # colcon test runs test/ with pytest
    zip_safe=True,
    maintainer="pusher-rl maintainers",
    maintainer_email="maintainers@pusher-rl.invalid",
    description="Shared plumbing of the pusher-rl nodes (no executables).",
    license="Apache-2.0",
    # A library package: no console_scripts.
    entry_points={"console_scripts": []},
)
