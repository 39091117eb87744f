from glob import glob

from setuptools import find_packages, setup

package_name = 'sphere_servo'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
    ],
    install_requires=['setuptools', 'numpy', 'pyyaml'],
    zip_safe=True,
    maintainer='sphere_servo developers',
    maintainer_email='sphere-servo@example.com',
    description='Visual servoing on a marked sphere with the minimal feature set s_n.',
    license='Apache-2.0',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'arm_sim = sphere_servo.nodes.arm_sim:main',
            'detector = sphere_servo.nodes.detector:main',
            'features = sphere_servo.nodes.features:main',
            'servo = sphere_servo.nodes.servo:main',
            'launcher = sphere_servo.tools.launcher:main',
            'record = sphere_servo.tools.record:main',
            'replay = sphere_servo.tools.replay:main',
            'refeatures = sphere_servo.tools.refeatures:main',
        ],
    },
)
