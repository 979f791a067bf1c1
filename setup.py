"""Packaging for flexure_ctrl (ROS 2 ament_python layout)."""

import os

from setuptools import find_packages
from setuptools import setup

PACKAGE_NAME = 'flexure_ctrl'
HERE = os.path.dirname(os.path.abspath(__file__))

# One entry per executable, 'name = module:function'.  colcon installs each one as
# <prefix>/lib/flexure_ctrl/<name> (see setup.cfg), where `ros2 run flexure_ctrl <name>`
# looks for it.  test/test_colcon_layout.py reads this list (through ast) and checks
# that every entry is installed there, so keep it a plain literal list of strings.
CONSOLE_SCRIPTS = [
    'flexure-ctrl = flexure_ctrl.cli.main:main',
    'trajectory_generator = flexure_ctrl.nodes.trajectory_generator:main',
    'inverse_solver = flexure_ctrl.nodes.inverse_solver:main',
    'actuator_loop = flexure_ctrl.nodes.actuator_loop:main',
    'tracker_bridge = flexure_ctrl.nodes.tracker_bridge:main',
    'recorder = flexure_ctrl.nodes.recorder:main',
    'player = flexure_ctrl.nodes.player:main',
]


def config_data_files(root='config'):
    """
    List every file under ``root`` as data_files entries, keeping subfolders.

    ``config/designs/a.yaml`` is installed as ``share/flexure_ctrl/config/designs/a.yaml``.
    Hidden files, editor backups and ``__pycache__`` folders are skipped.
    """
    entries = []
    top = os.path.join(HERE, root)
    for dirpath, dirnames, filenames in os.walk(top):
        dirnames[:] = sorted(
            d for d in dirnames if not d.startswith('.') and d != '__pycache__')
        rel_dir = os.path.relpath(dirpath, HERE)
        files = [
            os.path.join(rel_dir, f) for f in sorted(filenames)
            if not f.startswith('.') and not f.endswith(('~', '.pyc', '.swp'))
        ]
        if files:
            entries.append((os.path.join('share', PACKAGE_NAME, rel_dir), files))
    return entries


setup(
    name=PACKAGE_NAME,
    version='0.1.0',
    packages=find_packages(
        exclude=['test', 'test.*', 'bench', 'bench.*', 'scripts', 'scripts.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE_NAME]),
        ('share/' + PACKAGE_NAME, ['package.xml']),
    ] + config_data_files(),
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='flexure_ctrl developers',
    maintainer_email='dev@flexure-ctrl.invalid',
    description='Feedforward and feedback control of a bearing-free two-link flexure arm.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': CONSOLE_SCRIPTS,
    },
)
