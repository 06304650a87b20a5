"""Setuptools build of the ament_python package transplanter_ident (colcon and pip)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "transplanter_ident"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", sorted(glob("config/*.yaml"))),
        (f"share/{PACKAGE}/launch", sorted(glob("launch/*.py"))),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="transplanter_ident maintainers",
    maintainer_email="maintainer@example.com",
    description="Online IPSO-EKF identification of rice transplanter cornering stiffness",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            f"estimator = {PACKAGE}.ros.main:main",
            f"tuner = {PACKAGE}.cli.tuner:main",
            f"replay = {PACKAGE}.cli.replay:main",
            f"simulate = {PACKAGE}.cli.simulate:main",
            f"warm = {PACKAGE}.cli.warm:main",
        ],
    },
)
