"""Evaluations of the diagnosis on randomised simulated worlds.

``diagnose_benches`` (``online-id evaluate-diagnose``) and ``diagnose_rigs`` (``evaluate-diagnose-rig``) run the
diagnosis on the project's own bench and rig simulators and score it. The ``chain*`` modules
(``evaluate-diagnose-chain``) judge it from outside: randomised drivetrains built independently of the
product, written as users' files, the command line run as a user runs it, the answers scored against the
truth; they import nothing of the diagnosis (tests/test_architecture.py).
"""
