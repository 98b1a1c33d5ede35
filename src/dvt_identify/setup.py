from setuptools import find_namespace_packages, setup

package_name = 'dvt_identify'

setup(
    name=package_name,
    version='0.1.0',
    # namespace discovery: data folders (param sets, presets, descriptions) are packages too
    packages=find_namespace_packages(include=['dvt_identify', 'dvt_identify.*'], exclude=['*.__pycache__']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    package_data={package_name: ['py.typed', 'descriptions/*.yaml']},
    include_package_data=True,
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='dvt developers',
    maintainer_email='dvt@example.com',
    description='DVT identifier: output-error fits from bags, residual analysis and closed-loop model augmentation',
    license='Apache-2.0',
    extras_require={'test': ['pytest']},
    entry_points={'console_scripts': [
        'dvt-identify = dvt_identify.cli:main',
        'dvt_identify_node = dvt_identify.node:main',
        'dvt-import = dvt_identify.importer:main',
        'dvt-identify-batch = dvt_identify.batch_cli:main',
    ]},
)
