"""Build script of the ament_python package quatcal_ros (shape of ros2/demos, jazzy)."""

from glob import glob
import os

from setuptools import find_packages
from setuptools import setup

package_name = 'quatcal_ros'

# Files installed beside package.xml; `ros2 run`, launch files and get_package_share_directory()
# find them under share/quatcal_ros (config/*.yaml under share/quatcal_ros/config).
# config/ may not exist yet: glob() then returns [] and nothing is added.
data_files = [
    ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
    ('share/' + package_name, ['package.xml']),
]
config_files = sorted(glob(os.path.join('config', '*.yaml')))  # relative to this directory
if config_files:
    data_files.append(('share/' + package_name + '/config', config_files))
launch_files = sorted(glob(os.path.join('launch', '*.launch.py')))
if launch_files:
    data_files.append(('share/' + package_name + '/launch', launch_files))

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=data_files,
    install_requires=['setuptools'],
    extras_require={'test': ['pytest']},  # without it `colcon test` runs no tests
    zip_safe=True,
    maintainer='quatcal_ros maintainers',
    maintainer_email='quatcal@example.com',
    keywords=['ROS'],
    description='Hand-eye rotation calibration with the quaternion method of Chou and Kamel.',
    license='BSD-3-Clause',
    entry_points={
        'console_scripts': [
            'calibrator = quatcal_ros.ros.stop_signals:calibrator',
            'sim_cell = quatcal_ros.ros.stop_signals:sim_cell',
            'target_detector = quatcal_ros.ros.stop_signals:target_detector',
            'solve = quatcal_ros.__main__:solve',
            'replay = quatcal_ros.__main__:replay',
            'plan = quatcal_ros.__main__:plan',
            'demo = quatcal_ros.__main__:demo',
            'poses_to_bag = quatcal_ros.__main__:poses_to_bag',
        ],
    },
)
