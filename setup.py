from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'gcp_stereo_ros'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    package_data={PACKAGE: ['weights/*.pt', 'weights/*.confidence.json']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*')),
        ('share/' + PACKAGE + '/launch', glob('launch/*.launch.py')),
    ],
    # Runtime dependencies come from package.xml (rosdep) on a ROS install and from
    # requirements.txt (pinned) in a venv; listing them here would make setuptools'
    # script wrappers refuse to start when apt provides them under other names.
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='gcp_stereo_ros maintainers',
    maintainer_email='maintainers@gcp-stereo-ros.invalid',
    description='CNN ground control points steering semi-global matching, as a ROS 2 node',
    license='BSD-3-Clause',
    # Optional features, which rosdistro has no keys for: `pip install .[cluster]` for
    # gcp-stereo-batch on Ray, `.[cuda]` for device cuda (numba-cuda's kernels; a GPU also
    # needs a CUDA build of torch). colcon test picks its runner from 'test' (setuptools no
    # longer keeps tests_require). requirements.txt pins all of them for `make venv`.
    # numba-cuda 0.30's numpy overloads name np.row_stack, which numpy 2.5 removed: every
    # kernel failed to compile on a GPU machine that had numpy 2.5.
    extras_require={
        'cluster': ['ray'],
        'cuda': ['numba-cuda', 'cuda-bindings', 'cuda-core', 'nvidia-nvvm', 'nvidia-cuda-nvrtc',
                 'numpy<2.5'],
        'test': ['pytest'],
    },
    entry_points={
        'console_scripts': [
            'gcp_stereo_node = gcp_stereo_ros.node:main',
            'gcp_stereo_lifecycle_node = gcp_stereo_ros.ros.lifecycle_node:main',
            'point_cloud_node = gcp_stereo_ros.ros.point_cloud_node:main',
            'gcp-stereo-eval = gcp_stereo_ros.tools.evaluate:main',
            'gcp-stereo-bench = gcp_stereo_ros.tools.bench:main',
            'gcp-stereo-train = gcp_stereo_ros.tools.train:main',
            'gcp-stereo-plot = gcp_stereo_ros.tools.plot:main',
            'gcp-stereo-bag = gcp_stereo_ros.tools.bag:main',
            'gcp-stereo-batch = gcp_stereo_ros.tools.batch:main',
            'gcp-stereo-load = gcp_stereo_ros.tools.load:main',
            'gcp-stereo-demo = gcp_stereo_ros.tools.demo:main',
        ],
    },
)
