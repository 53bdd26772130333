from softphantom.cli import main


def test_version_and_unknown_command(capsys):
    assert main(["version"]) == 0
    assert "softphantom" in capsys.readouterr().out
    assert main(["no-such-command"]) == 2
