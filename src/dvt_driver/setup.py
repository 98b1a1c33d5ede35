from setuptools import find_namespace_packages, setup

package_name = 'dvt_driver'

setup(
    name=package_name,
    version='0.1.0',
    # namespace discovery: data folders (param sets, presets, descriptions) are packages too
    packages=find_namespace_packages(include=['dvt_driver', 'dvt_driver.*'], exclude=['*.__pycache__']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    package_data={package_name: ['py.typed', 'plant/config/*.yaml']},
    include_package_data=True,
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='dvt developers',
    maintainer_email='dvt@example.com',
    description='DVT serial link: wire protocol, lifecycle driver node, simulated plant, experiments, recorder, and the integration layer (launcher, loop benchmark, demo, dvt-bench)',
    license='Apache-2.0',
    extras_require={'test': ['pytest']},
    entry_points={'console_scripts': [
        'dvt_driver_node = dvt_driver.link.node:main',
        'dvt-plant = dvt_driver.plant.server:main',
        'dvt-experiment = dvt_driver.run.experiment:main',
        'dvt-recorder = dvt_driver.recording.node:main',
        'dvt-bag = dvt_driver.recording.bagtool:main',
        'dvt-launch = dvt_driver.system.launch:main',
        'dvt-foxglove = dvt_driver.run.foxglove:main',
        'dvt-discovery = dvt_driver.run.discovery:main',
        'dvt-bench = dvt_driver.system.bench:main',
    ]},
)
