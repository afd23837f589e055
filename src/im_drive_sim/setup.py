"""ament_python package im_drive_sim: its metadata, packages and data files are in setup.cfg."""

from setuptools import setup

setup()
