"""transplanter_ident: online IPSO-EKF identification of a rice transplanter's cornering stiffness."""

__version__ = "0.1.0"
