// The console's users file: what `pulsetrack console-user` writes, what `pulsetrack console`
// accepts, and every way a hand-edited or tampered file is refused with its file and line.

#include "pulsetrack/console/credentials.hpp"

#include <gtest/gtest.h>
#include <sys/stat.h>

#include <fstream>

#include "test_util.hpp"

namespace pulsetrack::console {
namespace {

TEST(ConsoleUsers, SetThenVerifyTheRightPasswordOnlyWithItsRole) {
  test::TempDir dir;
  const auto file = dir.path() / "users";
  ASSERT_TRUE(setUser(file, "surgeon", Role::kOperator, "correct horse", 2000));
  ASSERT_TRUE(setUser(file, "nurse", Role::kViewer, "battery staple", 2000));
  struct stat st {};
  ASSERT_EQ(stat(file.c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 0777, 0600U);  // password hashes: the owner's only
  auto c = Credentials::load(file);
  ASSERT_TRUE(c) << c.error().message;
  EXPECT_EQ(c->users().size(), 2U);
  EXPECT_EQ(c->verify("surgeon", "correct horse"), Role::kOperator);
  EXPECT_EQ(c->verify("nurse", "battery staple"), Role::kViewer);
  EXPECT_FALSE(c->verify("surgeon", "battery staple"));
  EXPECT_FALSE(c->verify("surgeon", "correct horsE"));
  EXPECT_FALSE(c->verify("nobody", "correct horse"));
  EXPECT_FALSE(c->verify("surgeon", ""));
  // The password is not in the file.
  std::ifstream in(file);
  const std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  EXPECT_EQ(text.find("correct horse"), std::string::npos);
  // A new password replaces the old one; the other user stays.
  ASSERT_TRUE(setUser(file, "surgeon", Role::kViewer, "new password", 2000));
  c = Credentials::load(file);
  ASSERT_TRUE(c);
  EXPECT_FALSE(c->verify("surgeon", "correct horse"));
  EXPECT_EQ(c->verify("surgeon", "new password"), Role::kViewer);
  EXPECT_EQ(c->verify("nurse", "battery staple"), Role::kViewer);
}

TEST(ConsoleUsers, BadNamesPasswordsAndFilesAreRefusedAndNamed) {
  test::TempDir dir;
  const auto file = dir.path() / "users";
  EXPECT_FALSE(setUser(file, "a b", Role::kOperator, "long enough"));
  EXPECT_FALSE(setUser(file, "x", Role::kOperator, "short"));
  auto missing = Credentials::load(dir.path() / "none");
  ASSERT_FALSE(missing);
  EXPECT_NE(missing.error().message.find("none: users file not found"), std::string::npos);
  const auto expect = [&](const std::string& content, const std::string& what) {
    { std::ofstream(file, std::ios::trunc) << content; }
    chmod(file.c_str(), 0600);
    auto c = Credentials::load(file);
    ASSERT_FALSE(c) << content;
    EXPECT_NE(c.error().message.find(what), std::string::npos) << c.error().message;
  };
  const std::string salt(32, 'a'), hash(64, 'b');
  expect("", "no user");
  expect("# only a comment\n", "no user");
  expect("a:operator:pbkdf2-sha256:2000:" + salt + "\n", "users:1: 5 fields");
  expect("\nbad name:operator:pbkdf2-sha256:2000:" + salt + ":" + hash + "\n", "users:2: the name");
  expect("a:root:pbkdf2-sha256:2000:" + salt + ":" + hash + "\n", "role 'root'");
  expect("a:viewer:md5:2000:" + salt + ":" + hash + "\n", "scheme 'md5'");
  expect("a:viewer:pbkdf2-sha256:10:" + salt + ":" + hash + "\n", "iterations must be");
  expect("a:viewer:pbkdf2-sha256:x:" + salt + ":" + hash + "\n", "iterations must be a number");
  expect("a:viewer:pbkdf2-sha256:2000:zz:" + hash + "\n", "the salt");
  expect("a:viewer:pbkdf2-sha256:2000:" + salt + ":abc\n", "the hash");
  expect("a:viewer:pbkdf2-sha256:2000:" + salt + ":" + hash +
             "\na:viewer:pbkdf2-sha256:2000:" + salt + ":" + hash + "\n",
         "users:2: user 'a' a second time");
  // Readable by others: refused (it holds password hashes).
  std::ofstream(file, std::ios::trunc)
      << "a:viewer:pbkdf2-sha256:2000:" << salt << ":" << hash << "\n";
  chmod(file.c_str(), 0644);
  auto open = Credentials::load(file);
  ASSERT_FALSE(open);
  EXPECT_NE(open.error().message.find("readable by others"), std::string::npos);
}

}  // namespace
}  // namespace pulsetrack::console
