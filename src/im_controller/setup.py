"""ament_python package: im_controller.

Executables are small shell wrappers installed as data files to
``<prefix>/lib/im_controller/`` -- the place ``ros2 run`` looks -- both under plain
``pip install`` (which ignores setup.cfg's install_scripts) and under colcon.
"""

from glob import glob

from setuptools import find_packages, setup

package_name = 'im_controller'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    package_data={package_name: ['config/*.yaml']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob(package_name + '/config/*.yaml')),
        ('lib/' + package_name, glob('scripts/*')),
    ],
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='im_tuner developers',
    maintainer_email='im-tuner@example.org',
    description='im_controller of the im_tuner project',
    license='Apache-2.0',
)
