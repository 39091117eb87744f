from glob import glob

from setuptools import find_packages, setup

package_name = 'sphere_servo'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(include=['sphere_servo', 'sphere_servo.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config/params', glob('config/params/*.yaml')),
        ('share/' + package_name + '/config/scenarios', glob('config/scenarios/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
        ('share/' + package_name + '/rosdep', glob('rosdep/*.yaml')),
        ('share/' + package_name + '/config', glob('config/fastdds*.xml')),
    ],
    # the runtime libraries, by their PyPI names (package.xml names their rosdep keys)
    install_requires=['setuptools', 'backports.zstd', 'example-robot-data', 'imageio-ffmpeg',
                      'lz4', 'matplotlib', 'meshcat', 'numpy', 'opencv-python-headless',
                      'pillow', 'pin', 'PyYAML', 'rosbags', 'u-msgpack-python'],
    zip_safe=True,
    maintainer='sphere_servo developers',
    maintainer_email='sphere-servo@example.com',
    description='Visual servoing on a marked sphere with the minimal feature set s_n.',
    license='Apache-2.0',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'arm_sim = sphere_servo.ros.arm_sim:main',
            'detector = sphere_servo.ros.detector:main',
            'features = sphere_servo.ros.features:main',
            'servo = sphere_servo.ros.servo:main',
            'launcher = sphere_servo.bringup.launcher:main',
            'pipeline = sphere_servo.bringup.single:main',
            'record = sphere_servo.bag.record:main',
            'replay = sphere_servo.bag.replay:main',
            'reindex = sphere_servo.bag.repair:main',
            'refeatures = sphere_servo.bag.refeatures:main',
        ],
    },
)
