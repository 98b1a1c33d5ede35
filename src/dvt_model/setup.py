from setuptools import find_namespace_packages, setup

package_name = 'dvt_model'

setup(
    name=package_name,
    version='0.1.0',
    # namespace discovery: data folders (param sets, presets, descriptions) are packages too
    packages=find_namespace_packages(include=['dvt_model', 'dvt_model.*'], exclude=['*.__pycache__']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    package_data={package_name: ['param_sets/*.yaml', 'design/*.yaml', 'py.typed']},
    include_package_data=True,
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='dvt developers',
    maintainer_email='dvt@example.com',
    description='DVT physics core (kinematics, Lagrangian dynamics, band brake, hybrid simulation) and the live model node',
    license='Apache-2.0',
    extras_require={'test': ['pytest']},
    entry_points={'console_scripts': [
        'dvt-model = dvt_model.cli:main',
        'dvt_model_node = dvt_model.node:main',
        'dvt-replay = dvt_model.replay:main',
    ]},
)
