"""ament_python package im_controller: its metadata, packages and data files are in setup.cfg."""

from setuptools import setup

setup()
