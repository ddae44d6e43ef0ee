def pytest_configure(config):
    config.addinivalue_line(
        'markers', 'notebooks: executes the example notebooks in examples/ '
        '(runs by default; deselect with -m "not notebooks")')
