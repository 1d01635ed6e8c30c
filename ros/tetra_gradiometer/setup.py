"""ament_python build description of the ROS package tetra_gradiometer (colcon).

The Python package, config, launch, security and bags/ are the checkout's, reached by the
symbolic links beside this file: the repository's root is no package, so colcon finds this
one and ../../tetra_gradiometer_msgs.
"""
from glob import glob

from setuptools import find_packages, setup

package_name = 'tetra_gradiometer'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(include=[package_name, package_name + '.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/config/scenarios', glob('config/scenarios/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
        ('share/' + package_name + '/security', glob('security/*.xml')),
        ('share/' + package_name + '/bags', glob('bags/*.yaml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='tetra_gradiometer maintainers',
    maintainer_email='maintainers@tetra-gradiometer.invalid',
    description='Vehicle magnetic interference compensation for a tetrahedral gradiometer',
    license='Apache-2.0',
    extras_require={'test': ['pytest', 'pytest-timeout']},
    entry_points={
        'console_scripts': [
            'driver = tetra_gradiometer.nodes.process:main_driver',
            'tensor = tetra_gradiometer.nodes.process:main_tensor',
            'calibrator = tetra_gradiometer.nodes.process:main_calibrator',
            'compensator = tetra_gradiometer.nodes.process:main_compensator',
            'target = tetra_gradiometer.nodes.process:main_target',
        ],
    },
)
