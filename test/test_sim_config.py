"""Simulator knobs: defaults, overrides, and errors that name the key."""

from flexure_ctrl.sim.config import load_sim_config, SimConfigError
import pytest


def test_defaults_have_the_interface_keys():
    config = load_sim_config()
    assert set(config['plant']) >= {'gravity_sag_scale', 'joint_offset_rad', 'joint_scale'}
    assert set(config['drives']) >= {'lag_s', 'max_speed_m_s', 'backlash_m', 'pot_noise_m',
                                     'drift_m_per_s'}
    assert set(config['tracker']) >= {'noise_m', 'rate_hz', 'dropout_probability'}
    assert 'seed' in config


def test_override_file_changes_only_its_keys(tmp_path):
    override = tmp_path / 'sim.yaml'
    override.write_text('plant: {gravity_sag_scale: 0}\ndrives: {backlash_m: 3.0e-4}\n'
                        'tracker: {dropout_probability: 0.01}\nseed: 7\n')
    config = load_sim_config(override)
    defaults = load_sim_config()
    assert config['plant']['gravity_sag_scale'] == 0.0
    assert config['drives']['backlash_m'] == 3.0e-4
    assert config['tracker']['dropout_probability'] == 0.01
    assert config['seed'] == 7
    assert config['drives']['lag_s'] == defaults['drives']['lag_s']


def test_command_line_overrides_come_last(tmp_path):
    override = tmp_path / 'sim.yaml'
    override.write_text('network: {can_port: 30001}\n')
    config = load_sim_config(override, {'network.can_port': 30002})
    assert config['network']['can_port'] == 30002


@pytest.mark.parametrize('text, key', [
    ('plant: {gravity_sag: 1.0}\n', 'plant.gravity_sag'),
    ('drives: {lag_s: fast}\n', 'drives.lag_s'),
    ('plant: {joint_scale: [1.0]}\n', 'plant.joint_scale'),
    ('tracker: 5\n', 'tracker'),
])
def test_unknown_or_mistyped_key_is_named(tmp_path, text, key):
    override = tmp_path / 'bad.yaml'
    override.write_text(text)
    with pytest.raises(SimConfigError, match=f"bad.yaml: .*'{key}'"):
        load_sim_config(override)
